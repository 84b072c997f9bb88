"""Recordings: MCAP topics, schemas, the writer, the columnar and reference readers, the recorded scenario,
the run summary computed from the telemetry."""
