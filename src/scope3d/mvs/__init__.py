"""Dense stereo for forward-looking scopes: axial-stereo geometry, matchers, confidence and fusion."""
