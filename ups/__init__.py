"""UPS: the Ulm Publisher/Subscriber protocol, one API across CAN buses and TCP/IP."""
