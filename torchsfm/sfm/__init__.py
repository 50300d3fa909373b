"""Structure from motion: two-view geometry and (later) reconstructions."""
