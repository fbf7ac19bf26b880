"""The ROS 2 wire as gridslam speaks it, shared by whoever talks to a ROS 2 graph: the messages
and their CDR (messages.py, numbers in, bytes out), rmw_zenoh's key expressions, QoS,
attachments and type hashes (rmw_zenoh.py), a node's liveliness tokens and its publishers and
subscribers on a Zenoh session (graph.py), and the node's place in the graph as flags, keys and
environment (graph_settings.py). The ros2 service (services/ros/node.py), the Foxglove bridge and
the MCAP export publish through it; the live `ros2:` source (services/source/ros2.py) reads
through it. docs/ecosystem.md.
"""
