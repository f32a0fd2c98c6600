"""Code shared by the algorithms."""
