"""What every data provider shares."""

from __future__ import annotations


class Provider:
    """Base of the data providers: keeps the params; :meth:`require` checks nothing unless a provider needs a
    setting made (``data=files`` needs its two paths)."""

    def __init__(self, params):
        self.p = params

    def require(self) -> None:
        return None
