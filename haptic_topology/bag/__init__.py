"""Recorded runs: reading rosbag2 (MCAP) bags of the node graph into traces."""
