//! Integration tests: map prepare.
