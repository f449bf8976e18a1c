"""Reading what users hand dyn_node (limits and trajectory files) safely: bounded, strict YAML and
JSON (:mod:`.safe_load`), regular files of bounded size (:mod:`.files`), and echoing their
values capped and escaped (:mod:`.text`); and what they get back in JSON (:mod:`.jsonable`).
No rclpy; only :mod:`.jsonable` imports NumPy."""
