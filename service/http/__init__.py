"""The HTTP shell: parse, call the core once, encode."""
