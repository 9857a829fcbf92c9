"""Real robot actors: UR arms through ur_rtde, RealSense cameras through pyrealsense2 (optional extras)."""
