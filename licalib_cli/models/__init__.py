"""Sensor models: IMU (method.md section 3) and per-beam LiDAR (method.md section 4)."""
