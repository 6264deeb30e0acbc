"""The robot server: pipelines (scan streamer, camera offloader) over one Zenoh session."""
