"""Light curves of satellites made of brdfjax facets (an edge package: it imports the core, config and io)."""
