"""Node shells of a live run: plant, encoder, attacker proxy, controller (``testbed node ...``)."""
