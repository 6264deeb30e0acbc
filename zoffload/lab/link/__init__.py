"""The network-condition emulator: a shaping TCP proxy driven by a time-varying trace."""
