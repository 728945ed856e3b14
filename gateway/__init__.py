"""The two-faced gateway between a CAN bus and a TCP/IP network."""
