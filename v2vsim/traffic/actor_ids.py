"""The ids of the actors a scenario places on purpose (no imports: the ego reads them without loading SUMO's
tools): the hidden foe (v2vsim/traffic/sumo_hidden_foe.py), the stopped car round the corner and the standing
vehicles (v2vsim/traffic/sumo_standing.py)."""

FOE_ID = "foe0"
HIDDEN_STOP_ID = "stopped0"
STANDING_PREFIX = "standing"
