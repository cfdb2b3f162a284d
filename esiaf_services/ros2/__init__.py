"""The ros2 service: ESIAF's voices as ROS4HRI (REP-155) topics over DDS, for ROS 2 nodes, without ROS."""
