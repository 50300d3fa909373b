"""Putative matching: NCC candidates in a disc, the strength measure and relaxation."""
