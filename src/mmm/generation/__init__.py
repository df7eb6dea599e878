"""Generation and editing with a trained text-to-motion model."""
