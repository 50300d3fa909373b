"""Independently moving objects (thesis chapter 5): plane + parallax, the parallax-based rigidity
constraint, IMOR (Alg. 5.4.1) and IMOR + RANSAC."""
