"""Camera control, capture sessions, manifests, scheduling and the ``hdrcap`` command line."""
