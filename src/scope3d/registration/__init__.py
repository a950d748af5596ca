"""Point-cloud registration: robust rigid 3-D-3-D fits (:mod:`.rigid`), statistical outlier removal
(:mod:`.outliers`) and the panoramic registration of side-view quadrants with loop closure
(:mod:`.panorama`, reference sec. 8.2-8.3)."""
