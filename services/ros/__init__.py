"""gridslam for ROS tools: a run's poses, map, images and transforms as ROS 2 messages, written
into an MCAP file (`run.mcap`, mcap_export.py), served live to Foxglove (foxglove.py), and
published live as a node of a ROS 2 graph over Zenoh (node.py: rmw_zenoh's wire format in
rmw_zenoh.py and graph.py, the node's state in projection.py). messages.py is the pure core they
share (numbers in, CDR bytes out). docs/ecosystem.md.

The ROS bag *source* (reading bags) is services/source/rosbag.py, the live ROS 2 source
services/source/ros2.py: it reads the ROS 2 wire through messages.py, rmw_zenoh.py, graph.py and
the graph's settings (graph_settings.py), never the services here.
"""
