"""The catalogue feature: ingesting scans, the cards' pages and images, the 3D viewer and the
homography check."""
