"""``python -m dyn_node.ros.demo [--short] [--out DIR]``."""
from dyn_node.ros.demo.driver import main

raise SystemExit(main())
