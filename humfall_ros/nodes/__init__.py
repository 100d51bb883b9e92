"""humfall_ros.nodes"""
