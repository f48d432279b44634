"""TRACE-GS framework."""
