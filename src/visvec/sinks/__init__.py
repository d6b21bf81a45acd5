"""Where rows go: CSV or JSON lines, flushed row by row, to a file, stdout or UDP."""

from visvec.sinks.writers import CsvSink, JsonlSink, UdpStream, open_sink

__all__ = ["CsvSink", "JsonlSink", "UdpStream", "open_sink"]
