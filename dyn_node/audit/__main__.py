"""``python -m dyn_node.audit``: the same as the ``dyn-audit`` command."""
import gc

if __name__ == "__main__":
    gc.disable()  # no collection during the imports (bag_audit's reason); main() turns it back on

from dyn_node.audit.bag_audit import main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(main())
