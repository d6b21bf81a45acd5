"""Where rows go: CSV or JSON lines, flushed row by row."""

from visvec.sinks.writers import CsvSink, JsonlSink, open_sink

__all__ = ["CsvSink", "JsonlSink", "open_sink"]
