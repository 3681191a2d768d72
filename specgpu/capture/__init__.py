"""Capture: drivers, the ring buffer and the sequence assembler."""
