"""dyn-fleet: many bags audited as Ray tasks, fleet tables and page."""
