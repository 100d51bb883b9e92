"""humfall_ros.estop"""
