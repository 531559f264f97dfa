"""Task families; each module registers its variants with `registry`."""
