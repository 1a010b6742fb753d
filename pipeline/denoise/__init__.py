"""The uncertainty-driven bilateral filter (Sec. 9) and its tiled form for images larger than memory."""
