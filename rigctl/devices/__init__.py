"""Wire protocols and host-side clients of the rig's two boards."""
