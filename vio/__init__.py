"""vio room."""
