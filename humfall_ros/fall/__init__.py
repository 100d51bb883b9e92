"""humfall_ros.fall"""
