"""The classical observers: Kalman filters and smoother, the EKF on the car that slips, and the
classical registry."""
