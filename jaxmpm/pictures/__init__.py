"""Pictures and export of a finished run: snapshots read back as per-point fields
(`snapshots`), figures and animations (`plotting`), ParaView files (`export`)."""
