"""Event readers and writers (the io helper fills this in)."""
