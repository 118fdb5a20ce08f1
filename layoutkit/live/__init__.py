"""Live mode: sources, protocols, decoding, pipeline, statistics, dashboard, hardware simulator."""
