"""Everything that touches a camera: ``camera/`` (the protocol, its errors, the gphoto2 and
simulated backends) and ``capture/`` (sessions, manifests, jobs, run folders, schedules)."""
