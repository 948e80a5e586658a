"""The world as every stage after the traffic simulator sees it: `state` (WorldState, actors, the static
map), `geometry` (poses, frames, the BEV grid) and `serialize` (their bytes on the driver -> agents link)."""
