"""3D products whose values stay temperatures: per-pixel correction, textures, facade mosaics, exports."""
