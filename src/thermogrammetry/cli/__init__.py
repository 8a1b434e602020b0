"""Command-line interface: parses, prints, shows progress; the work is in the library."""
