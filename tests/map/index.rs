//! Integration tests: map index.
