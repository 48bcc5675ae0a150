"""The clinician web pages under /ui/ (server-rendered HTML and SVG)."""
