"""Video files in and out, drawing tracks on frames, and exporting tracks to npz and csv."""
