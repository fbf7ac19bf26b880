"""gridslam for ROS tools: a run's poses, map, images and transforms as ROS 2 messages, written
into an MCAP file (`run.mcap`, mcap_export.py) or served live to Foxglove (foxglove.py).
messages.py is the pure core both share (numbers in, CDR bytes out). docs/ecosystem.md.

The ROS bag *source* (reading bags) is services/source/rosbag.py.
"""
