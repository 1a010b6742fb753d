"""Camera wrappers that stand for what happens to a rig around the camera."""

from __future__ import annotations

import os
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


class _Kill:
    """Stands for the stop event of :class:`StoppingCamera`: delivers the real SIGTERM instead."""

    def stop(self, signum):
        os.kill(os.getpid(), signum)


class SignallingCamera(StoppingCamera):
    """A camera that receives SIGTERM (as from `systemctl stop`) after ``after`` captures and
    records whether it was closed."""

    def __init__(self, cam, after: int):
        super().__init__(cam, _Kill(), after)
        self.closed = False

    def close(self):
        self.closed = True
        self._cam.close()
