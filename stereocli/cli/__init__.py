"""Command line (Click only): parse, validate, call the library, report."""
