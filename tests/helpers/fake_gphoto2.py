"""A simulated camera body behind the worker protocol of the gphoto2 backend, in this process."""

from __future__ import annotations

from pathlib import Path


class FakeBody:
    """A simulated PTP body behind the worker protocol of ``Gphoto2Camera`` (in this process):
    RAW+JPEG pairs named DSC_nnnn, events queued with delays (a number of 50-ms waits that
    time out first), a bulb widget (``bulb`` toggle or Canon's ``eosremoterelease``), storages."""

    def __init__(self, raw_delay=0, fmt="NEF+Fine", canon=False, storages=None, longest="30"):
        self.dead, self.pid, self.n = False, 4242, 0
        self.queue: list = []  # [delay, (kind, data)]
        self.raw_delay, self.canon = raw_delay, canon
        self.storages = storages if storages is not None else [{"freeimages": 100, "access": "rw"}]
        labels = ["1/100", "1/10", "1", longest, "Bulb"]
        self.widgets = {
            "shutterspeed": ("radio", "1/100", labels),
            "imagequality": ("radio", fmt, [fmt]),
            "capturetarget": ("radio", "Memory card", ["Internal RAM", "Memory card"]),
            "serialnumber": ("text", "F00D", []),
        }
        if canon:
            self.widgets["eosremoterelease"] = ("radio", "None", ["None", "Press Full", "Release Full"])
        else:
            self.widgets["bulb"] = ("toggle", 0, [])
        self.log: list = []

    def call(self, op, *args, timeout=None):
        self.log.append(op)
        return getattr(self, "op_" + op)(*args)

    def stop(self, timeout=0.0):
        self.dead = True

    def op_detect(self):
        return [("Fake Body", "usb:001,002")]

    def op_open(self, model, port):
        pass

    def op_exit(self):
        pass

    def _find(self, names):
        return next((n for n in names if n in self.widgets), None)

    def op_describe(self, names):
        n = self._find(names)
        if n is None:
            return None
        typ, value, choices = self.widgets[n]
        return {"name": n, "type": typ, "value": value, "choices": list(choices), "readonly": False}

    def op_read(self, names):
        n = self._find(names)
        return None if n is None else self.widgets[n][1]

    def op_set(self, name, value):
        typ, _old, choices = self.widgets[name]
        self.widgets[name] = (typ, value, choices)
        return value

    def op_storage(self):
        return self.storages

    def _shoot(self, announce_jpeg):
        self.n += 1
        jpg, raw = ("/store/DCIM", f"DSC_{self.n:04d}.JPG"), ("/store/DCIM", f"DSC_{self.n:04d}.NEF")
        if announce_jpeg:
            self.queue.append([0, ("file", jpg)])
        self.queue.append([self.raw_delay, ("file", raw)])
        return jpg

    def op_capture(self):
        return self._shoot(announce_jpeg=False)

    def op_trigger(self):
        self._shoot(announce_jpeg=True)

    def op_bulb(self, name, press, release, seconds):
        self.log.append(("bulb", name, press, release))
        self._shoot(announce_jpeg=True)
        return {"press_start": 0.0, "press_end": 0.01, "release_start": seconds + 0.004, "release_end": seconds + 0.02}

    def op_event(self, ms):
        if not self.queue:
            return "timeout", ""
        if self.queue[0][0] > 0:
            self.queue[0][0] -= 1
            return "timeout", ""
        return self.queue.pop(0)[1]

    def op_drain(self, ms):
        out = []
        while self.queue:
            self.queue[0][0] = 0  # everything pending arrives while draining
            out.append(self.queue.pop(0)[1])
        return out

    def op_download(self, folder, name, path):
        Path(path).write_text(name)

    def op_delete(self, folder, name):
        pass


def fake_camera(body, **kw):
    """A ``Gphoto2Camera`` whose worker is ``body`` (in this process)."""
    from hdrcap.acquire.camera.gphoto2 import Gphoto2Camera

    cls = type("FakeGphoto2Camera", (Gphoto2Camera,), {"worker_factory": staticmethod(lambda name: body)})
    return cls(**kw)
