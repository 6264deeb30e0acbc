"""zoffload: offload a mobile robot's LiDAR mapping and perception to an edge computer over Zenoh."""

__version__ = "0.1.0"
