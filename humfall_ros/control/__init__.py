"""humfall_ros.control"""
