//! `texel-viewer`: renders the texel model (arrives with the viewer issue).

fn main() -> anyhow::Result<()> {
    anyhow::bail!("texel-viewer: the renderer is not built yet; see the README")
}
