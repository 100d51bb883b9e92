"""humfall_ros.multicontact"""
