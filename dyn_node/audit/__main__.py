"""``python -m dyn_node.audit``: the same as the ``dyn-audit`` command."""
from dyn_node.audit.bag_audit import main

if __name__ == "__main__":
    raise SystemExit(main())
