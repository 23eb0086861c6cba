"""Filters: the interaction matrix, the velocity Kalman filter and the pose UKF."""
