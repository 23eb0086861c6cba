"""Sequence folder format (being written)."""


class Sequence:  # replaced in this issue
    pass
