"""Demo robots: CAN nodes and TCP hosts talking through UPS."""
