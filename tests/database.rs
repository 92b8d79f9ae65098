//! Integration tests: database.
