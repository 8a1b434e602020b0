"""Test helper: a verb run as its own process, its stderr read as it comes, and a wait for a progress line."""

from __future__ import annotations

import subprocess
import sys
import threading
import time


class VerbProcess:
    """``python -m thermogrammetry ARGS`` started now; ``lines`` fills with its stderr in a reader thread."""

    def __init__(self, args, *, new_session: bool = False):
        self.p = subprocess.Popen([sys.executable, "-m", "thermogrammetry", *map(str, args)], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, start_new_session=new_session)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=lambda: self.lines.extend(self.p.stderr), daemon=True)
        self._reader.start()

    def wait_for_line(self, text: str, timeout_s: float) -> bool:
        """Wait until a stderr line holds ``text`` (or the process ends, or ``timeout_s``); True while it still runs."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s and self.p.poll() is None and not any(text in ln for ln in self.lines):
            time.sleep(0.02)
        return self.p.poll() is None

    def finish(self, timeout_s: float) -> str:
        """Wait for the end; returns all of stderr."""
        self.p.wait(timeout=timeout_s)
        self._reader.join(timeout=30)
        return "".join(self.lines)
