"""humfall_ros.dynamics"""
