"""The edge server: services (mapping, detection) over one Zenoh session."""
