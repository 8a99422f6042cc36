"""Depth sources behind one interface: replay, freenect, openni2, oak, synthetic."""
