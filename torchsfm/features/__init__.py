"""Feature detection: Harris corners with the biquadric sub-pixel fit."""
