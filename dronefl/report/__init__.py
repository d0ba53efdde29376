"""Tables and plots (the only place matplotlib is imported)."""
