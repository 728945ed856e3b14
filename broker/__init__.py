"""Event Channel Brokers: the CAN-ECB (TxNodes, etags) and the TCP/IP-ECB (subscription lists)."""
