"""humfall_ros: humanoid fall handling (detection, safe fall, e-stop, multi-contact planning)."""
__version__ = "0.1.0"
