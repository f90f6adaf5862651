//! Who may do what through the web UI, and the headers every page carries.
//!
//! Reads are open (the map shows what the gateway publishes over MQTT
//! anyway). Writes (route requests, survey, saving a site) are refused when
//! `[web] read_only`, and need the token (`Authorization: Bearer …`) when
//! the server is bound anywhere but loopback. Two browser attacks are shut
//! out even on loopback: another site's page posting to the gateway
//! (cross-site requests: writes must carry a JSON or binary body, which a
//! cross-origin page cannot send without a CORS preflight this server never
//! grants, and a same-origin `Origin` if any), and DNS rebinding (a
//! loopback-bound server answers only to loopback host names).
//!
//! Every response carries a strict Content-Security-Policy: scripts and
//! styles from this server only, nothing inline, no frames, no plugins; the
//! pages never build HTML from data (names and ids from the air go in as
//! text), so even a missed case cannot run a script.

use std::net::SocketAddr;
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

pub const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; script-src 'self'; \
     style-src 'self'; img-src 'self'; connect-src 'self'; font-src 'none'; object-src 'none'; \
     form-action 'none'; frame-ancestors 'none'; base-uri 'none'";

/// The access rules of one server.
#[derive(Debug)]
pub(super) struct Guard {
    read_only: bool,
    /// Bound off loopback: writes need the token.
    needs_token: bool,
    token: Option<String>,
    /// The port of a loopback-bound server, whose `Host` must be a loopback
    /// name (DNS rebinding); `None` off loopback.
    loopback_port: Option<u16>,
}

impl Guard {
    pub(super) fn new(bind: SocketAddr, read_only: bool, token: Option<String>) -> Guard {
        let loopback = bind.ip().is_loopback();
        Guard {
            read_only,
            needs_token: !loopback,
            token,
            loopback_port: loopback.then_some(bind.port()),
        }
    }

    /// What the pages are told: whether they may offer writes, and whether
    /// they must ask for the token. Never the token itself.
    pub(super) fn access(&self) -> serde_json::Value {
        serde_json::json!({
            "read_only": self.read_only || (self.needs_token && self.token.is_none()),
            "needs_token": self.needs_token,
        })
    }

    fn host_allowed(&self, headers: &HeaderMap) -> bool {
        let Some(port) = self.loopback_port else {
            return true;
        };
        let Some(host) = headers.get(header::HOST).and_then(|h| h.to_str().ok()) else {
            return false;
        };
        let (name, given_port) = match host.strip_prefix('[') {
            Some(rest) => match rest.split_once(']') {
                Some((ip, tail)) => (ip, tail.strip_prefix(':')),
                None => return false,
            },
            None => match host.rsplit_once(':') {
                Some((name, p)) => (name, Some(p)),
                None => (host, None),
            },
        };
        if given_port.is_some_and(|p| p.parse::<u16>().ok() != Some(port)) {
            return false;
        }
        name == "localhost"
            || name.ends_with(".localhost")
            || name
                .parse::<std::net::IpAddr>()
                .is_ok_and(|ip| ip.is_loopback())
    }

    /// Why a write is refused, if it is.
    fn refuse_write(&self, headers: &HeaderMap) -> Option<(StatusCode, &'static str, String)> {
        if self.read_only {
            return Some((
                StatusCode::FORBIDDEN,
                "read_only",
                "this gateway serves the map only ([web] read_only = true)".into(),
            ));
        }
        let body_kind = headers
            .get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("");
        let body_kind = body_kind.split(';').next().unwrap_or("").trim();
        if !matches!(body_kind, "application/json" | "application/octet-stream") {
            return Some((
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "bad_request",
                "writes carry application/json (or application/octet-stream for images)".into(),
            ));
        }
        if let (Some(origin), Some(host)) = (headers.get(header::ORIGIN), headers.get(header::HOST))
        {
            let same = origin
                .to_str()
                .ok()
                .and_then(|o| o.split_once("://"))
                .is_some_and(|(_, rest)| rest.as_bytes() == host.as_bytes());
            if !same {
                return Some((
                    StatusCode::FORBIDDEN,
                    "cross_origin",
                    "writes are taken only from this gateway's own pages".into(),
                ));
            }
        }
        if !self.needs_token {
            return None;
        }
        let Some(token) = &self.token else {
            return Some((
                StatusCode::FORBIDDEN,
                "no_token",
                "this gateway is reachable off loopback and has no write token, so it serves \
                 the map only; set [web] token_file (or the systemd credential web-token)"
                    .into(),
            ));
        };
        let given = headers
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .unwrap_or("");
        if !same_secret(given.as_bytes(), token.as_bytes()) {
            return Some((
                StatusCode::UNAUTHORIZED,
                "unauthorized",
                "this write needs the gateway's web token".into(),
            ));
        }
        None
    }
}

/// Compares without stopping at the first difference, so the time taken
/// does not tell an attacker how much of a guess was right.
fn same_secret(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// An error reply in the shape every API error has.
pub(super) fn error(status: StatusCode, code: &str, message: impl Into<String>) -> Response {
    let body = serde_json::json!({ "error": { "code": code, "message": message.into() } });
    (status, axum::Json(body)).into_response()
}

/// The middleware: host check, write rules, then the security headers.
pub(super) async fn guard(
    State(guard): State<Arc<Guard>>,
    request: Request,
    next: Next,
) -> Response {
    let headers = request.headers();
    let mut response = if !guard.host_allowed(headers) {
        error(
            StatusCode::MISDIRECTED_REQUEST,
            "bad_host",
            "this gateway listens on loopback and answers only to localhost names",
        )
    } else if !matches!(*request.method(), Method::GET | Method::HEAD) {
        match guard.refuse_write(headers) {
            Some((status, code, message)) => error(status, code, message),
            None => next.run(request).await,
        }
    } else {
        next.run(request).await
    };
    let h = response.headers_mut();
    let set = |h: &mut HeaderMap, name: header::HeaderName, value: &'static str| {
        h.insert(name, HeaderValue::from_static(value));
    };
    set(h, header::CONTENT_SECURITY_POLICY, CONTENT_SECURITY_POLICY);
    set(h, header::X_CONTENT_TYPE_OPTIONS, "nosniff");
    set(h, header::X_FRAME_OPTIONS, "DENY");
    set(h, header::REFERRER_POLICY, "no-referrer");
    h.insert(
        header::HeaderName::from_static("cross-origin-opener-policy"),
        HeaderValue::from_static("same-origin"),
    );
    h.insert(
        header::HeaderName::from_static("cross-origin-resource-policy"),
        HeaderValue::from_static("same-origin"),
    );
    if !h.contains_key(header::CACHE_CONTROL) {
        set(h, header::CACHE_CONTROL, "no-store");
    }
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(&str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(
                header::HeaderName::from_bytes(k.as_bytes()).unwrap(),
                HeaderValue::from_str(v).unwrap(),
            );
        }
        h
    }

    #[test]
    fn a_loopback_server_answers_only_to_loopback_names() {
        let g = Guard::new("127.0.0.1:8080".parse().unwrap(), false, None);
        for ok in [
            "127.0.0.1:8080",
            "localhost:8080",
            "[::1]:8080",
            "localhost",
        ] {
            assert!(g.host_allowed(&headers(&[("host", ok)])), "{ok}");
        }
        for bad in [
            "evil.example:8080",
            "127.0.0.1:9999",
            "evil.example",
            "10.0.0.1:8080",
        ] {
            assert!(!g.host_allowed(&headers(&[("host", bad)])), "{bad}");
        }
        assert!(!g.host_allowed(&HeaderMap::new()));
        let open = Guard::new("0.0.0.0:8080".parse().unwrap(), false, None);
        assert!(open.host_allowed(&headers(&[("host", "gateway.lan:8080")])));
    }

    #[test]
    fn writes_need_json_the_same_origin_and_off_loopback_the_token() {
        let json = ("content-type", "application/json");
        let local = Guard::new("127.0.0.1:8080".parse().unwrap(), false, None);
        assert!(local.refuse_write(&headers(&[json])).is_none());
        let form = headers(&[("content-type", "text/plain")]);
        assert_eq!(local.refuse_write(&form).unwrap().1, "bad_request");
        let cross = headers(&[
            json,
            ("origin", "http://evil.example"),
            ("host", "127.0.0.1:8080"),
        ]);
        assert_eq!(local.refuse_write(&cross).unwrap().1, "cross_origin");
        let same = headers(&[
            json,
            ("origin", "http://127.0.0.1:8080"),
            ("host", "127.0.0.1:8080"),
        ]);
        assert!(local.refuse_write(&same).is_none());

        let token = "0123456789abcdef0123";
        let open = Guard::new("0.0.0.0:8080".parse().unwrap(), false, Some(token.into()));
        assert_eq!(
            open.refuse_write(&headers(&[json])).unwrap().1,
            "unauthorized"
        );
        let wrong = headers(&[json, ("authorization", "Bearer 0123456789abcdef0124")]);
        assert_eq!(open.refuse_write(&wrong).unwrap().1, "unauthorized");
        let right = headers(&[json, ("authorization", &format!("Bearer {token}"))]);
        assert!(open.refuse_write(&right).is_none());
        let tokenless = Guard::new("0.0.0.0:8080".parse().unwrap(), false, None);
        assert_eq!(tokenless.refuse_write(&right).unwrap().1, "no_token");
        assert_eq!(tokenless.access()["read_only"], true);
        let read_only = Guard::new("127.0.0.1:8080".parse().unwrap(), true, None);
        assert_eq!(
            read_only.refuse_write(&headers(&[json])).unwrap().1,
            "read_only"
        );
    }
}
