"""Captures of a lit skin point: the ingest stage (brackets -> HDR -> radial profiles)
and the capture simulator."""
