"""Where rows go: CSV or JSON lines, flushed row by row, to a file, stdout or UDP
(writers), or ROS 2 messages in an MCAP file (ros)."""

from visvec.sinks.writers import CsvSink, JsonlSink, Tee, UdpStream, open_sink, row_writer

__all__ = ["CsvSink", "JsonlSink", "Tee", "UdpStream", "open_sink", "row_writer"]
