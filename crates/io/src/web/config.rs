//! `[web]` in the gateway config: where the browser UI listens and who may
//! change things through it.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use serde::Deserialize;

/// Name of the systemd credential read when `token_file` is unset.
pub(crate) const TOKEN_CREDENTIAL: &str = "web-token";
/// The shortest token taken: shorter ones are guessed.
const MIN_TOKEN_LEN: usize = 16;

#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WebConfig {
    /// Serve the browser UI at all.
    pub enabled: bool,
    /// Address and port to listen on. Loopback by default: bound anywhere
    /// else, every write needs the token.
    pub bind: SocketAddr,
    /// Serve the map alone: no route requests, survey or saving.
    pub read_only: bool,
    /// The file holding the token writes need when bound off loopback
    /// (default: the systemd credential `web-token`).
    pub token_file: Option<PathBuf>,
    /// Where survey mode appends its fingerprints (default: `survey.csv` in
    /// `$STATE_DIRECTORY` under systemd, else beside the config file); on a
    /// building of several floors, a file per floor (`{floor}` in the path,
    /// else `-NAME` before its extension).
    pub survey_file: Option<PathBuf>,
}

impl Default for WebConfig {
    fn default() -> Self {
        WebConfig {
            enabled: true,
            bind: SocketAddr::from(([127, 0, 0, 1], 8080)),
            read_only: false,
            token_file: None,
            survey_file: None,
        }
    }
}

impl WebConfig {
    pub(crate) fn resolve_paths(&mut self, base: &Path) {
        if let Some(file) = &mut self.token_file {
            *file = base.join(&*file);
        }
        let state = std::env::var_os("STATE_DIRECTORY").map(PathBuf::from);
        let survey = self.survey_file.take();
        self.survey_file = Some(match survey {
            Some(file) => base.join(file),
            None => state.as_deref().unwrap_or(base).join("survey.csv"),
        });
    }

    /// Whether writes need the token: bound anywhere but loopback.
    pub(crate) fn needs_token(&self) -> bool {
        !self.bind.ip().is_loopback()
    }

    /// The write token: from `token_file`, else the systemd credential, else
    /// none. A file that is named but unreadable, or a token too short to
    /// resist guessing, is an error.
    pub(crate) fn token(&self) -> Result<Option<String>, String> {
        let path = match &self.token_file {
            Some(p) => p.clone(),
            None => match std::env::var_os("CREDENTIALS_DIRECTORY") {
                Some(dir) if Path::new(&dir).join(TOKEN_CREDENTIAL).exists() => {
                    Path::new(&dir).join(TOKEN_CREDENTIAL)
                }
                _ => return Ok(None),
            },
        };
        let text = std::fs::read_to_string(&path)
            .map_err(|e| format!("[web] cannot read the token file {}: {e}", path.display()))?;
        let token = text.trim().to_owned();
        if token.len() < MIN_TOKEN_LEN || token.chars().any(|c| c.is_control() || c == ' ') {
            return Err(format!(
                "[web] the token in {} must be at least {MIN_TOKEN_LEN} characters with no \
                 spaces (for example: `head -c 24 /dev/urandom | base64`)",
                path.display()
            ));
        }
        Ok(Some(token))
    }
}
