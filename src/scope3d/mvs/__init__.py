"""Dense stereo: axial stereo for forward-looking scopes (:mod:`.axial`, :mod:`.dense_matching`,
:mod:`.confidence`, compiled :mod:`.axial_kernels` and :mod:`.refine_kernels`), two-view and multi-view
fusion (:mod:`.two_view`, :mod:`.multiview`), a plane sweep with known poses (:mod:`.plane_sweep`), the map
points new frames no longer see (:mod:`.surface_change`) and a cavity's wall textured from the frames
(:mod:`.texturing`)."""
