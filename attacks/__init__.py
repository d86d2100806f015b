"""Attack objects placed in scenes."""
