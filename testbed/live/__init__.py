"""A live run's launcher: spawning and supervising the nodes, the collector, the live Rerun and Foxglove taps."""
