"""The optimisers as ``(init, update)`` pairs, their one loop and history, one fit, and the global search."""
