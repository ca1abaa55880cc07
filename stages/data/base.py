"""What every data provider shares."""

from __future__ import annotations


class Provider:
    """Base of the data providers: keeps the params; :meth:`require` checks nothing unless a provider needs a
    setting made (``data=files`` needs its two paths)."""

    def __init__(self, params):
        self.p = params

    def require(self) -> None:
        return None

    def preflight(self) -> None:
        """What can be checked without reading a scan: :meth:`require`, and in providers that read files, that
        they are there. A sweep checks every job so before its first job starts (:mod:`scanreg.app.sweep`), so
        that a typo in one swept value stops the sweep at once instead of failing when that job's turn comes."""
        self.require()
