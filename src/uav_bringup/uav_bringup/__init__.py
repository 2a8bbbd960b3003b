"""Flying and watching the stack: the fly launcher, MCAP recording and the Foxglove live view."""
