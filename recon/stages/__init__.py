"""Stage entry points: the only modules that read or write the run folder (through RunPaths)."""
