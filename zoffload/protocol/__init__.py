"""The wire protocol: message types and their codec, every key expression, scan payload coding,
and the checks every received message passes."""
