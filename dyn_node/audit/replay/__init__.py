"""dyn-audit's replay machinery: the configurations read from the bag (config), each topic's role
(roles), the replay of the inputs (inputs) with one replayer per kind of recorded event (contact,
services, gates), the re-check of the recorded outputs (recheck) and what they share (common,
stats)."""
