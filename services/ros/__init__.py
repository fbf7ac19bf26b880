"""gridslam for ROS tools: a run's poses, map, images and transforms as ROS 2 messages, written
into an MCAP file (`run.mcap`, mcap_export.py), served live to Foxglove (foxglove.py), and
published live as a node of a ROS 2 graph over Zenoh (node.py, the node's state in
projection.py). The wire they share — messages, CDR, rmw_zenoh's keys and the graph — is
services/ros2wire, which the live ROS 2 source (services/source/ros2.py) reads too. The ROS bag
*source* (reading bags) is services/source/rosbag.py. docs/ecosystem.md.
"""
