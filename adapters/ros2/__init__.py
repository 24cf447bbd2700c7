"""The ros2 transport: an unmodified ROS 2 node is the target (Cyclone DDS, ROS 2's
topics, types and CDR; no harness protocol on the wire).

``link`` the harness half (``Ros2Link``) · ``target`` the SDK's node (``serve_endpoint``) ·
``options`` (``Ros2Options``: domain, discovery, topics, QoS, the control mapping) ·
``answers`` ROS 2 messages <-> frames and estimates · ``dds`` Cyclone participants ·
``msgs`` the message types (``msg/``: definitions rosbags lacks) · ``cdr`` their bytes.
"""
