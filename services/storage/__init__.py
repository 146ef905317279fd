"""Object storage for the warm and cold tiers: one small interface, backends chosen by URL scheme."""
