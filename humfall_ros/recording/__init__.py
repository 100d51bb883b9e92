"""humfall_ros.recording"""
