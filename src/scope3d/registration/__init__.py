"""Registration: 2-D mosaics of scope frames (and, later, 3-D panoramic registration)."""
