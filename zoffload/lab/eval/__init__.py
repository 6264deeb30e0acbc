"""Metrics and plots: trajectory error, receive-time statistics, result figures."""
