//! Integration tests: map projection.
