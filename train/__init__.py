"""Lightning training of the pose network (the pose-network issue)."""
