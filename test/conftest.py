"""Shared set-up of the ROS tests: real DDS, kept on this machine and off other runs' domains."""

import os

# Before any rclpy context exists: discovery on localhost only, and a domain of our own so
# that parallel CI jobs and a user's running ROS graph never see each other.
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(11 + os.getpid() % 90))
os.environ.pop('ROS_LOCALHOST_ONLY', None)
os.environ.setdefault('RERUN_ANALYTICS', '0')
