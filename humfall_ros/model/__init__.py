"""humfall_ros.model"""
