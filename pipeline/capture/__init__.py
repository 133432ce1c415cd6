"""Stage 3, capture: the ring protocol, host client, emulator, cameras and the capture plan."""
