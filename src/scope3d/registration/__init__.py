"""Registration: robust rigid 3-D-3-D fits (:mod:`.rigid`), statistical outlier removal (:mod:`.outliers`),
the panoramic registration of side-view quadrants with loop closure (:mod:`.panorama`, reference sec.
8.2-8.3), and 2-D mosaics of scope frames with global alignment (:mod:`.mosaic`, reference ch. 2)."""
