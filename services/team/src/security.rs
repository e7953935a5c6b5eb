//! Who may join the team link: Zenoh TLS with mutual authentication (every robot and router
//! holds a certificate of the team CA, [`crate::certs`]) and Zenoh access control naming
//! each robot by its certificate's common name.
//!
//! What each robot `X` of the roster (`[team.tls] robots`) may do, enforced by every robot
//! and router on its links (`<T>` = the team name, key expressions of [`crate::link`]):
//!
//! | from `X` (ingress) | key expressions |
//! |---|---|
//! | put (messages) | `doorslam/<T>/*/*/X`: only as the sender `X` |
//! | liveliness token | `doorslam/<T>/alive/X`: only its own |
//! | subscriber | `doorslam/<T>/X/*/*`: only its own inbox |
//! | liveliness subscriber and query | `doorslam/<T>/alive/*` |
//!
//! and what goes to `X` (egress): messages addressed to it (`doorslam/<T>/X/*/*`), the
//! team's tokens and subscribers. Routers (common name
//! [`crate::certs::ROUTER_COMMON_NAME`]) forward everything under the team's prefix and
//! apply the same rules to the robots connected to them. Anything else is denied: a
//! certificate of the team CA whose common name is not in the roster can open a link and
//! do nothing; a peer without a certificate of the CA cannot open a link (the TLS handshake
//! fails), and plain TCP is not accepted at all (`transport/link/protocols = ["tls"]`).
//!
//! Zenoh's access control names subjects one by one (no templates in Zenoh 1.10): that is
//! why the roster is configured. Discovery still needs no list: robots of the roster come
//! and go by their liveliness tokens.

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use doorslam_ipc::wire::RobotId;
use serde::Deserialize;
use serde_json::json;
use x509_parser::prelude::{FromDer, X509Certificate};

use crate::certs::ROUTER_COMMON_NAME;
use crate::link::TeamError;

/// `[team.tls]` of robot.toml (and of the router's config): absent = plain TCP, open to
/// anyone on the network.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsSection {
    /// The team CA's certificate (`ca.pem` of `doorslam team certs`).
    pub ca: PathBuf,
    /// This robot's (or router's) certificate, signed by the CA.
    pub cert: PathBuf,
    /// Its private key.
    pub key: PathBuf,
    /// Robot ids holding team certificates: the access control lets each one publish only
    /// under its own id.
    pub robots: Vec<String>,
}

impl TlsSection {
    /// The roster, checked (the files are checked by [`Security::check`] at start-up).
    pub fn roster(&self) -> Result<Vec<RobotId>, String> {
        if self.robots.is_empty() {
            return Err("robots: list the robot ids holding team certificates".into());
        }
        self.robots
            .iter()
            .map(|r| {
                RobotId::new(r)
                    .map_err(|_| format!("robots: {r:?} is not a robot id ([a-z0-9_-], 1-32)"))
            })
            .collect()
    }
}

/// Whose certificate a process holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Holder {
    Robot(RobotId),
    Router,
}

impl Holder {
    pub fn common_name(&self) -> &str {
        match self {
            Holder::Robot(id) => id.as_str(),
            Holder::Router => ROUTER_COMMON_NAME,
        }
    }
}

/// What is wrong with a TLS file; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    #[error("{path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: not PEM ({expected} expected)")]
    NotPem {
        path: PathBuf,
        expected: &'static str,
    },
    #[error("{path}: not an X.509 certificate: {reason}")]
    Certificate { path: PathBuf, reason: String },
    #[error("{path}: not a CA certificate (no CA basic constraint)")]
    NotCa { path: PathBuf },
    #[error("{path}: not signed by the team CA {ca}")]
    NotSignedByCa { path: PathBuf, ca: PathBuf },
    #[error("{path}: expired on {not_after} (renew it with doorslam team certs; is this clock right? robots without a synchronized clock need doorslam team certs --clockless)")]
    Expired { path: PathBuf, not_after: String },
    #[error("{path}: not valid before {not_before} (is this clock right? robots without a synchronized clock need doorslam team certs --clockless)")]
    NotYetValid { path: PathBuf, not_before: String },
    #[error("{path}: common name {found:?}, this process is {expected:?} (a robot's certificate names its robot id)")]
    CommonName {
        path: PathBuf,
        found: String,
        expected: String,
    },
    #[error("{path}: not a private key: {reason}")]
    Key { path: PathBuf, reason: String },
    #[error("{key}: not the private key of {cert}")]
    KeyMismatch { key: PathBuf, cert: PathBuf },
    #[error("[team.tls] {0}")]
    Roster(String),
    #[error("{0}: not valid UTF-8 (Zenoh's config takes paths as strings)")]
    Path(PathBuf),
}

/// The parts of a certificate the checks use.
#[derive(Debug, Clone)]
pub(crate) struct CertInfo {
    der: Vec<u8>,
    pub common_name: Option<String>,
    pub organization: Option<String>,
    /// The subject public key (raw bit string).
    pub public_key: Vec<u8>,
    pub not_before: i64,
    pub not_after: i64,
    pub is_ca: bool,
}

fn date(unix_s: i64) -> String {
    x509_parser::time::ASN1Time::from_timestamp(unix_s)
        .map(|t| t.to_string())
        .unwrap_or_else(|_| format!("{unix_s} s after 1970"))
}

/// The first certificate of a PEM file.
pub(crate) fn parse_certificate_pem(path: &Path, bytes: &[u8]) -> Result<CertInfo, SecurityError> {
    let not_pem = || SecurityError::NotPem {
        path: path.into(),
        expected: "a CERTIFICATE block",
    };
    let pem = x509_parser::pem::Pem::iter_from_buffer(bytes)
        .next()
        .ok_or_else(not_pem)?
        .map_err(|_| not_pem())?;
    if pem.label != "CERTIFICATE" {
        return Err(SecurityError::NotPem {
            path: path.into(),
            expected: "a CERTIFICATE block, found a different one",
        });
    }
    let bad = |reason: String| SecurityError::Certificate {
        path: path.into(),
        reason,
    };
    let (_, cert) = X509Certificate::from_der(&pem.contents).map_err(|e| bad(e.to_string()))?;
    let common_name = cert
        .subject()
        .iter_common_name()
        .next()
        .and_then(|a| a.as_str().ok())
        .map(str::to_string);
    let organization = cert
        .subject()
        .iter_organization()
        .next()
        .and_then(|a| a.as_str().ok())
        .map(str::to_string);
    let is_ca = cert
        .basic_constraints()
        .map_err(|e| bad(format!("basic constraints: {e}")))?
        .is_some_and(|b| b.value.ca);
    Ok(CertInfo {
        common_name,
        organization,
        public_key: cert.public_key().subject_public_key.data.to_vec(),
        not_before: cert.validity().not_before.timestamp(),
        not_after: cert.validity().not_after.timestamp(),
        is_ca,
        der: pem.contents.clone(),
    })
}

fn read(path: &Path) -> Result<Vec<u8>, SecurityError> {
    std::fs::read(path).map_err(|source| SecurityError::Read {
        path: path.into(),
        source,
    })
}

fn unix_now() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs() as i64)
}

fn check_validity(path: &Path, c: &CertInfo, now: i64) -> Result<(), SecurityError> {
    if now > c.not_after {
        return Err(SecurityError::Expired {
            path: path.into(),
            not_after: date(c.not_after),
        });
    }
    if now < c.not_before {
        return Err(SecurityError::NotYetValid {
            path: path.into(),
            not_before: date(c.not_before),
        });
    }
    Ok(())
}

/// The checked TLS settings of one process: what [`Security::apply`] puts in its Zenoh config.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Security {
    pub team: String,
    pub ca: PathBuf,
    pub cert: PathBuf,
    pub key: PathBuf,
    pub roster: Vec<RobotId>,
    /// When this process's certificate expires (Unix seconds); Zenoh closes the links then.
    pub expires_unix_s: i64,
}

impl Security {
    /// Checks the files of `tls` for `holder` (errors name the file and what is wrong:
    /// missing, not PEM, not signed by the CA, expired, another common name, a key that is
    /// not the certificate's) and the roster.
    pub fn check(tls: &TlsSection, team: &str, holder: &Holder) -> Result<Self, SecurityError> {
        Self::check_at(tls, team, holder, unix_now())
    }

    /// [`Security::check`] with the wall clock reading `now_unix_s` (a robot whose clock is
    /// off: clockless certificates pass whatever it reads, dated ones say which date failed).
    pub fn check_at(
        tls: &TlsSection,
        team: &str,
        holder: &Holder,
        now_unix_s: i64,
    ) -> Result<Self, SecurityError> {
        let roster = tls.roster().map_err(SecurityError::Roster)?;
        let now = now_unix_s;
        let ca = parse_certificate_pem(&tls.ca, &read(&tls.ca)?)?;
        if !ca.is_ca {
            return Err(SecurityError::NotCa {
                path: tls.ca.clone(),
            });
        }
        check_validity(&tls.ca, &ca, now)?;
        let cert = parse_certificate_pem(&tls.cert, &read(&tls.cert)?)?;
        verify_signed_by(&tls.cert, &cert, &tls.ca, &ca)?;
        check_validity(&tls.cert, &cert, now)?;
        if cert.common_name.as_deref() != Some(holder.common_name()) {
            return Err(SecurityError::CommonName {
                path: tls.cert.clone(),
                found: cert.common_name.unwrap_or_default(),
                expected: holder.common_name().into(),
            });
        }
        let key_text = String::from_utf8(read(&tls.key)?).map_err(|_| SecurityError::NotPem {
            path: tls.key.clone(),
            expected: "a PRIVATE KEY block",
        })?;
        if !key_text.contains("-----BEGIN") {
            return Err(SecurityError::NotPem {
                path: tls.key.clone(),
                expected: "a PRIVATE KEY block",
            });
        }
        let key = rcgen::KeyPair::from_pem(&key_text).map_err(|e| SecurityError::Key {
            path: tls.key.clone(),
            reason: e.to_string(),
        })?;
        if key.public_key_raw() != cert.public_key {
            return Err(SecurityError::KeyMismatch {
                key: tls.key.clone(),
                cert: tls.cert.clone(),
            });
        }
        for p in [&tls.ca, &tls.cert, &tls.key] {
            if p.to_str().is_none() {
                return Err(SecurityError::Path(p.clone()));
            }
        }
        let days_left = (cert.not_after - now) / 86_400;
        if days_left < 14 && cert.not_after < crate::certs::CLOCKLESS_NOT_AFTER_UNIX_S as i64 {
            tracing::warn!(
                cert = %tls.cert.display(),
                days_left,
                "team certificate expires soon: renew it with doorslam team certs"
            );
        }
        if let Holder::Robot(me) = holder {
            if !roster.contains(me) {
                tracing::warn!(robot = %me, "[team.tls] robots does not list this robot: the other robots' rosters must, or they refuse it");
            }
        }
        Ok(Self {
            team: team.to_string(),
            ca: tls.ca.clone(),
            cert: tls.cert.clone(),
            key: tls.key.clone(),
            roster,
            expires_unix_s: cert.not_after,
        })
    }

    /// TLS with mutual authentication on every link, only TLS links, and the access control
    /// of the module docs.
    pub fn apply(&self, config: &mut zenoh::Config) -> Result<(), TeamError> {
        let mut set = |key: &'static str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| TeamError::Config {
                    key,
                    reason: e.to_string(),
                })
        };
        let path = |p: &Path| json!(p.to_str().unwrap_or_default()).to_string();
        set("transport/link/protocols", r#"["tls"]"#.into())?;
        set("transport/link/tls/root_ca_certificate", path(&self.ca))?;
        set("transport/link/tls/listen_certificate", path(&self.cert))?;
        set("transport/link/tls/listen_private_key", path(&self.key))?;
        set("transport/link/tls/connect_certificate", path(&self.cert))?;
        set("transport/link/tls/connect_private_key", path(&self.key))?;
        set("transport/link/tls/enable_mtls", "true".into())?;
        // Robots are reached by address, not by a DNS name: the CA's signature and the
        // access control on the common name decide who a peer is.
        set("transport/link/tls/verify_name_on_connect", "false".into())?;
        set("transport/link/tls/close_link_on_expiration", "true".into())?;
        set(
            "access_control",
            access_control(&self.team, &self.roster).to_string(),
        )?;
        Ok(())
    }

    /// Time left before this process's certificate expires (zero if it has).
    pub fn time_left(&self) -> Duration {
        Duration::from_secs(self.expires_unix_s.saturating_sub(unix_now()).max(0) as u64)
    }
}

fn verify_signed_by(
    path: &Path,
    cert: &CertInfo,
    ca_path: &Path,
    ca: &CertInfo,
) -> Result<(), SecurityError> {
    let not_signed = || SecurityError::NotSignedByCa {
        path: path.into(),
        ca: ca_path.into(),
    };
    let (_, c) = X509Certificate::from_der(&cert.der).map_err(|_| not_signed())?;
    let (_, issuer) = X509Certificate::from_der(&ca.der).map_err(|_| not_signed())?;
    c.verify_signature(Some(issuer.public_key()))
        .map_err(|_| not_signed())
}

/// Zenoh's `access_control` for a team and its roster (the table of the module docs).
pub fn access_control(team: &str, roster: &[RobotId]) -> serde_json::Value {
    let all_messages = format!("doorslam/{team}/*/*/*");
    let alive = format!("doorslam/{team}/alive/*");
    let mut rules = vec![
        json!({"id": "team-liveliness", "permission": "allow", "flows": ["ingress", "egress"],
               "messages": ["declare_liveliness_subscriber", "liveliness_query"],
               "key_exprs": [alive]}),
        json!({"id": "to-any-tokens", "permission": "allow", "flows": ["egress"],
               "messages": ["liveliness_token"], "key_exprs": [alive]}),
        json!({"id": "to-any-subscribers", "permission": "allow", "flows": ["egress"],
               "messages": ["declare_subscriber"], "key_exprs": [all_messages]}),
        json!({"id": "router", "permission": "allow", "flows": ["ingress", "egress"],
               "messages": ["put", "declare_subscriber"], "key_exprs": [all_messages]}),
        json!({"id": "router-tokens", "permission": "allow", "flows": ["ingress", "egress"],
               "messages": ["liveliness_token"], "key_exprs": [alive]}),
    ];
    let mut subjects = vec![
        json!({"id": "routers", "cert_common_names": [ROUTER_COMMON_NAME],
                                   "link_protocols": ["tls"]}),
    ];
    let mut policies = vec![json!({"id": "routers",
        "rules": ["team-liveliness", "router", "router-tokens"], "subjects": ["routers"]})];
    for r in roster {
        let r = r.as_str();
        rules.push(
            json!({"id": format!("from-{r}"), "permission": "allow", "flows": ["ingress"],
            "messages": ["put"], "key_exprs": [format!("doorslam/{team}/*/*/{r}")]}),
        );
        rules.push(json!({"id": format!("token-of-{r}"), "permission": "allow",
            "flows": ["ingress"], "messages": ["liveliness_token"],
            "key_exprs": [format!("doorslam/{team}/alive/{r}")]}));
        rules.push(json!({"id": format!("inbox-of-{r}"), "permission": "allow",
            "flows": ["ingress"], "messages": ["declare_subscriber"],
            "key_exprs": [format!("doorslam/{team}/{r}/*/*")]}));
        rules.push(
            json!({"id": format!("to-{r}"), "permission": "allow", "flows": ["egress"],
            "messages": ["put"], "key_exprs": [format!("doorslam/{team}/{r}/*/*")]}),
        );
        subjects.push(json!({"id": format!("robot-{r}"), "cert_common_names": [r],
                             "link_protocols": ["tls"]}));
        policies.push(json!({"id": format!("robot-{r}"),
            "rules": ["team-liveliness", "to-any-tokens", "to-any-subscribers",
                      format!("from-{r}"), format!("token-of-{r}"), format!("inbox-of-{r}"),
                      format!("to-{r}")],
            "subjects": [format!("robot-{r}")]}));
    }
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

/// Endpoints must all be `tls/` with TLS on, and none without it.
pub fn check_endpoints(
    endpoints: &[String],
    what: &'static str,
    tls: bool,
) -> Result<(), TeamError> {
    for e in endpoints {
        let is_tls = e.starts_with("tls/");
        if tls && !is_tls {
            return Err(TeamError::Config {
                key: what,
                reason: format!("{e}: with [team.tls] every endpoint must be tls/<address>:<port>"),
            });
        }
        if !tls && is_tls {
            return Err(TeamError::Config {
                key: what,
                reason: format!("{e}: a tls/ endpoint needs [team.tls] (ca, cert, key, robots)"),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, SystemTime};

    use super::*;
    use crate::certs::{generate, CertsRequest, TeamCa, Validity};

    struct Files {
        _dir: tempfile::TempDir,
        root: PathBuf,
    }

    fn team(robots: &[&str]) -> Files {
        team_with(robots, false)
    }

    fn team_with(robots: &[&str], clockless: bool) -> Files {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().to_path_buf();
        generate(
            &root,
            &CertsRequest {
                team: "t1".into(),
                robots: robots.iter().map(|s| s.to_string()).collect(),
                routers: vec!["r1".into()],
                days: 30,
                clockless,
            },
        )
        .unwrap();
        Files { _dir: dir, root }
    }

    fn section(f: &Files, robot: &str) -> TlsSection {
        let d = f.root.join("robots").join(robot);
        TlsSection {
            ca: f.root.join("ca.pem"),
            cert: d.join("cert.pem"),
            key: d.join("key.pem"),
            robots: vec!["a".into(), "b".into()],
        }
    }

    fn robot(id: &str) -> Holder {
        Holder::Robot(RobotId::new(id).unwrap())
    }

    #[test]
    fn team_certificates_pass_and_the_config_takes_tls_and_the_access_control() {
        let f = team(&["a", "b"]);
        let s = Security::check(&section(&f, "a"), "t1", &robot("a")).unwrap();
        assert_eq!(s.roster.len(), 2);
        assert!(s.time_left() > Duration::from_secs(29 * 86_400));
        let mut config = zenoh::Config::default();
        s.apply(&mut config).unwrap();
        // The router's certificate names the router, not a robot.
        let r = f.root.join("routers/r1");
        let router = TlsSection {
            cert: r.join("cert.pem"),
            key: r.join("key.pem"),
            ..section(&f, "a")
        };
        Security::check(&router, "t1", &Holder::Router).unwrap();
        let err = Security::check(&router, "t1", &robot("a")).unwrap_err();
        assert!(matches!(err, SecurityError::CommonName { .. }), "{err}");
    }

    const YEAR_S: i64 = 365 * 86_400;

    #[test]
    fn a_robot_whose_clock_is_years_off_passes_with_clockless_certificates_only() {
        let now = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .unwrap()
            .as_secs() as i64;
        // A drone without RTC at boot (1970 plus a day), one years behind, one years ahead.
        let clocks = [86_400, now - 5 * YEAR_S, now + 30 * YEAR_S];
        let dated = team(&["a", "b"]);
        let clockless = team_with(&["a", "b"], true);
        for clock in clocks {
            let err =
                Security::check_at(&section(&dated, "a"), "t1", &robot("a"), clock).unwrap_err();
            assert!(
                matches!(
                    err,
                    SecurityError::NotYetValid { .. } | SecurityError::Expired { .. }
                ),
                "clock {clock}: {err}"
            );
            assert!(err.to_string().contains("--clockless"), "{err}");
            let s = Security::check_at(&section(&clockless, "a"), "t1", &robot("a"), clock)
                .unwrap_or_else(|e| panic!("clock {clock}: {e}"));
            assert_eq!(
                s.expires_unix_s,
                crate::certs::CLOCKLESS_NOT_AFTER_UNIX_S as i64
            );
        }
        // Authentication is intact with the clock off: another team's certificate, or a
        // certificate for another robot, is still refused.
        let other = team_with(&["a"], true);
        let foreign = TlsSection {
            cert: other.root.join("robots/a/cert.pem"),
            key: other.root.join("robots/a/key.pem"),
            ..section(&clockless, "a")
        };
        let err = Security::check_at(&foreign, "t1", &robot("a"), 86_400).unwrap_err();
        assert!(matches!(err, SecurityError::NotSignedByCa { .. }), "{err}");
        let err =
            Security::check_at(&section(&clockless, "b"), "t1", &robot("a"), 86_400).unwrap_err();
        assert!(matches!(err, SecurityError::CommonName { .. }), "{err}");
    }

    #[test]
    fn a_clockless_team_refuses_to_reuse_a_dated_ca() {
        let dated = team(&["a"]);
        let err = generate(
            &dated.root,
            &CertsRequest {
                team: "t1".into(),
                robots: vec!["c".into()],
                routers: vec![],
                days: 30,
                clockless: true,
            },
        )
        .unwrap_err();
        assert!(err.to_string().contains("not a clockless CA"), "{err}");
        // The other way round is fine: a dated robot certificate under a clockless CA.
        let clockless = team_with(&["a"], true);
        assert!(TeamCa::load(&clockless.root)
            .unwrap()
            .unwrap()
            .is_clockless());
        assert!(!TeamCa::load(&dated.root).unwrap().unwrap().is_clockless());
    }

    #[test]
    fn errors_name_the_file_and_what_is_wrong() {
        let f = team(&["a", "b"]);
        let good = section(&f, "a");
        let msg = |s: &TlsSection, holder: &Holder| {
            Security::check(s, "t1", holder).unwrap_err().to_string()
        };
        // Missing file.
        let missing = TlsSection {
            cert: f.root.join("nope.pem"),
            ..good.clone()
        };
        let e = msg(&missing, &robot("a"));
        assert!(e.contains("nope.pem") && e.contains("No such file"), "{e}");
        // Not PEM.
        let garbage = f.root.join("garbage.pem");
        std::fs::write(&garbage, "hello").unwrap();
        let e = msg(
            &TlsSection {
                cert: garbage.clone(),
                ..good.clone()
            },
            &robot("a"),
        );
        assert!(e.contains("garbage.pem") && e.contains("not PEM"), "{e}");
        let e = msg(
            &TlsSection {
                key: garbage.clone(),
                ..good.clone()
            },
            &robot("a"),
        );
        assert!(e.contains("garbage.pem") && e.contains("not PEM"), "{e}");
        // A key PEM where the certificate should be.
        let e = msg(
            &TlsSection {
                cert: good.key.clone(),
                ..good.clone()
            },
            &robot("a"),
        );
        assert!(e.contains("key.pem") && e.contains("CERTIFICATE"), "{e}");
        // The CA's place taken by a robot certificate.
        let e = msg(
            &TlsSection {
                ca: good.cert.clone(),
                ..good.clone()
            },
            &robot("a"),
        );
        assert!(e.contains("not a CA"), "{e}");
        // Another team's CA signed it.
        let other = team(&["a"]);
        let e = msg(
            &TlsSection {
                cert: other.root.join("robots/a/cert.pem"),
                key: other.root.join("robots/a/key.pem"),
                ..good.clone()
            },
            &robot("a"),
        );
        assert!(e.contains("not signed by the team CA"), "{e}");
        // b's key with a's certificate.
        let e = msg(
            &TlsSection {
                key: f.root.join("robots/b/key.pem"),
                ..good.clone()
            },
            &robot("a"),
        );
        assert!(
            e.contains("robots/b/key.pem") && e.contains("not the private key of"),
            "{e}"
        );
        // a's certificate for robot b.
        let e = msg(&good, &robot("b"));
        assert!(e.contains("common name \"a\""), "{e}");
        // Expired, and not yet valid.
        let ca = TeamCa::load(&f.root).unwrap().unwrap();
        let day = Duration::from_secs(86_400);
        let now = SystemTime::now();
        for (name, validity, what) in [
            (
                "old",
                Validity {
                    not_before: now - day * 10,
                    not_after: now - day,
                },
                "expired",
            ),
            (
                "new",
                Validity {
                    not_before: now + day,
                    not_after: now + day * 10,
                },
                "not valid before",
            ),
        ] {
            let (cert, key) = ca.issue("a", validity).unwrap();
            let (cp, kp) = (
                f.root.join(format!("{name}.pem")),
                f.root.join(format!("{name}.key")),
            );
            std::fs::write(&cp, cert).unwrap();
            std::fs::write(&kp, key).unwrap();
            let e = msg(
                &TlsSection {
                    cert: cp,
                    key: kp,
                    ..good.clone()
                },
                &robot("a"),
            );
            assert!(
                e.contains(&format!("{name}.pem")) && e.contains(what),
                "{e}"
            );
        }
        // A roster entry that is not a robot id.
        let e = msg(
            &TlsSection {
                robots: vec!["a".into(), "B*".into()],
                ..good.clone()
            },
            &robot("a"),
        );
        assert!(e.contains("B*"), "{e}");
    }

    #[test]
    fn access_control_names_each_robot_once_and_only_under_its_id() {
        let roster = [RobotId::new("a").unwrap(), RobotId::new("b").unwrap()];
        let acl = access_control("t1", &roster);
        assert_eq!(acl["default_permission"], "deny");
        let rule = |id: &str| {
            acl["rules"]
                .as_array()
                .unwrap()
                .iter()
                .find(|r| r["id"] == id)
                .unwrap()
                .clone()
        };
        assert_eq!(rule("from-a")["key_exprs"][0], "doorslam/t1/*/*/a");
        assert_eq!(rule("from-a")["flows"][0], "ingress");
        assert_eq!(rule("token-of-b")["key_exprs"][0], "doorslam/t1/alive/b");
        assert_eq!(rule("to-b")["key_exprs"][0], "doorslam/t1/b/*/*");
        let subjects = acl["subjects"].as_array().unwrap();
        assert_eq!(subjects.len(), 3);
        assert!(subjects
            .iter()
            .any(|s| s["cert_common_names"][0] == ROUTER_COMMON_NAME));
        // Endpoints: only tls/ with TLS, none without.
        assert!(check_endpoints(&["tcp/1.2.3.4:7447".into()], "listen", true).is_err());
        assert!(check_endpoints(&["tls/1.2.3.4:7447".into()], "listen", false).is_err());
        assert!(check_endpoints(&["tls/1.2.3.4:7447".into()], "listen", true).is_ok());
    }
}
