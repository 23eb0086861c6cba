"""Pose networks, their registry, keypoint decoding and PnP (the pose-network issue)."""
