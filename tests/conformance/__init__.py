"""CAN conformance: our CAN-ECB and our node against docs/protocol.md, frames built from its
tables only (``_frames``)."""
