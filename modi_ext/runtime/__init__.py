"""How a call finds its path and checks it (filled in below)."""
