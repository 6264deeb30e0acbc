"""Everything that runs the product for research: the demo, the experiments, the link emulator,
evaluation and reports. Depends on the product, never the other way."""
