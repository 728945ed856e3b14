"""The tests' EtherCAT slave emulator (test code, not a feature): ``_sii`` the SII EEPROM
image, ``_esc`` one slave controller and its AL state machine, ``_chain`` a line of slaves
that a frame passes through, ``__main__`` the process on a raw socket (``python -m tests.ecat
--help``). docs/ethercat.md describes what it emulates."""
