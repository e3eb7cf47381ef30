"""controllers room."""
