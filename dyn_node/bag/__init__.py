"""Bag I/O without ROS: CDR, the MCAP writer and reader, the recorder, recovery of damaged bags."""
