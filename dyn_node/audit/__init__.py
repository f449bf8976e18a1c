"""Offline analysis through the same core: dyn-audit (bag replay), evidence records, HTML reports, dyn-check (trajectory files)."""
