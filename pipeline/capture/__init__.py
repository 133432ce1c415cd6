"""Stage 3, capture: the ring protocol, host client, emulator, cameras and the capture plan, and
the recordings read as captures (a video file, ``video_frames``; the DiLiGenT layout, ``diligent``)."""
