"""Event optical flow by triplet matching with RoI registration."""
