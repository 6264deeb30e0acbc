"""Process plumbing: settings, errors and exit codes, lifecycle and signals, Zenoh sessions,
monitors, CPU quota, the router."""
