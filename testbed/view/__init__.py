"""Drawing a run: the Rerun and Foxglove views and the phase-plane geometry both share."""
