"""REST routers, one per resource; ``service.app`` mounts them behind the API key."""
