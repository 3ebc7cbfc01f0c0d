"""Small tools for looking at the package's own cost (op and host-sync counts)."""
