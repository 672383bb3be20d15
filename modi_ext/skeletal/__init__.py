"""The skeletal ops (filled in below)."""
