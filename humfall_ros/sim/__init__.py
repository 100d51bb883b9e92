"""humfall_ros.sim"""
