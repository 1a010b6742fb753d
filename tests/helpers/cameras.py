"""Camera wrappers that stand for what happens to a rig around the camera."""

from __future__ import annotations

import signal


class StoppingCamera:
    """A MockCamera whose stop event is set (as SIGTERM would) after ``after`` captures."""

    def __init__(self, cam, stop, after):
        self._cam, self._stop, self._after, self.n = cam, stop, after, 0

    def __getattr__(self, name):
        return getattr(self._cam, name)

    def capture(self, *a, **kw):
        res = self._cam.capture(*a, **kw)
        self.n += 1
        if self.n == self._after:
            self._stop.stop(signal.SIGTERM)
        return res
