"""ChArUco board definition, detection and stereo calibration, shared by processing and depth validation."""
