//! Integration tests: map.
mod index;
mod io;
mod prepare;
mod projection;
