"""One router per resource: health/readiness, the model card, registration."""
