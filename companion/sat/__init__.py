"""The GM-PHD search-and-track core: pure functions over arrays of components."""
