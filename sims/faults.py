"""Fault injection shared by every firmware simulator (serial ones and the USB camera)."""
from __future__ import annotations

import threading
from collections import Counter


class FaultInjection:
    """Faults armed with :meth:`inject` and consumed one occurrence at a time.

    A simulator lists the faults it models in ``FAULTS`` and calls :meth:`take_fault` where each
    one can strike. Subclasses create ``self.faults = Counter()`` and ``self._lock`` (an RLock)
    in ``__init__`` (see :meth:`_init_faults`).
    """

    FAULTS: frozenset[str] = frozenset()

    def _init_faults(self) -> None:
        self.faults: Counter[str] = Counter()
        self._lock = threading.RLock()

    def inject(self, fault: str, count: int = 1) -> None:
        """Arm ``fault`` for its next ``count`` occurrences.

        Raises
        ------
        ValueError
            If ``fault`` is not one this simulator models (a typo would otherwise arm nothing
            and a fault test would pass without its fault), or ``count`` < 1.
        """
        if fault not in self.FAULTS:
            raise ValueError(f"{type(self).__name__}: unknown fault {fault!r}; "
                             f"known: {', '.join(sorted(self.FAULTS))}")
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        with self._lock:
            self.faults[fault] += count

    def take_fault(self, fault: str) -> bool:
        """Consume one armed ``fault``; True if it was armed."""
        with self._lock:
            if self.faults[fault] > 0:
                self.faults[fault] -= 1
                return True
            return False

    def clear_faults(self) -> None:
        with self._lock:
            self.faults.clear()
