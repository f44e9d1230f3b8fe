//! What the hub keeps for radiance (protocol version 4): each exposed scan's
//! `ScanExposure` frame, sent to version 4 clients just before the scan's
//! `ScanAdded` (broadcast or fetched), and the session's `EoResponse` frame, sent in
//! their snapshots. About 40 bytes a scan, kept for the session (a scan's frame may be
//! dropped from memory and read back from the store; its exposure stays here).

use std::collections::HashMap;

use bytes::Bytes;
use texel::EoExposure;
use texel::model::ScanId;
use texel::radiance::EoResponse;
use texel::wire::Message;

use super::{Hub, HubError};

#[derive(Debug, Default)]
pub(super) struct Radiance {
    exposures: HashMap<ScanId, Bytes>,
    response: Option<Bytes>,
}

impl Radiance {
    pub(super) fn exposure(&self, id: ScanId) -> Option<&Bytes> {
        self.exposures.get(&id)
    }

    pub(super) fn response(&self) -> Option<&Bytes> {
        self.response.as_ref()
    }
}

impl Hub {
    /// How scan `id`'s EO frame was exposed; call before [`Hub::add_scan`], whose
    /// broadcast sends it first to the clients that speak version 4.
    pub fn note_exposure(&self, id: ScanId, exposure: &EoExposure) -> Result<(), HubError> {
        let frame = Message::ScanExposure {
            id,
            exposure: *exposure,
        }
        .encode()?;
        self.lock()
            .radiance
            .exposures
            .insert(id, Bytes::from(frame));
        Ok(())
    }

    /// The session's EO response curve (`None`: the sensor model has none), given to
    /// version 4 clients in their snapshots from now on.
    pub fn set_eo_response(&self, response: Option<&EoResponse>) -> Result<(), HubError> {
        let frame = match response {
            Some(r) => Some(Bytes::from(
                Message::EoResponse(Box::new(r.clone())).encode()?,
            )),
            None => None,
        };
        self.lock().radiance.response = frame;
        Ok(())
    }
}
