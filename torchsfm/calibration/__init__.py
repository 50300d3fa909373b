"""Camera calibration from chessboard photos (thesis §2.1.3, Appendix A: Zhang's method)."""
