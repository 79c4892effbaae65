"""Small shared helpers: seeding, box geometry, logging."""
