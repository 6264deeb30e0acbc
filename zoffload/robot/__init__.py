"""The robot daemon: sensor replay, per-scan downsampling, offloading, counters."""
