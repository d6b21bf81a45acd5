"""The `visvec` command line (click). Commands parse, call the library, format."""
