//! The texel model viewer: stream client, view-dependent renderer and headless rendering.
