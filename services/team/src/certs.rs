//! Team certificates (`doorslam team certs`): one certificate authority per team, and one
//! certificate + private key per robot and per router, signed by it. A robot's certificate
//! names the robot id as its common name and its subject alternative name, so Zenoh's
//! access control can name it (see [`crate::security`]); every router's common name is
//! [`ROUTER_COMMON_NAME`], which no robot id can equal (ids have no `.`).
//!
//! Layout of the output folder:
//!
//! | file | what | where it goes |
//! |---|---|---|
//! | `ca.pem` | the team CA's certificate | every robot and router |
//! | `ca.key` | the CA's private key | nowhere: kept by whoever issues certificates (reused to add robots) |
//! | `robots/<id>/cert.pem`, `key.pem` | robot `<id>`'s certificate and key | robot `<id>` only |
//! | `routers/<name>/cert.pem`, `key.pem` | a router's certificate and key | that router only |
//!
//! Keys are ECDSA P-256, written with mode 0600. An existing `ca.pem` + `ca.key` in the
//! folder is reused (robots added later join the same team); an existing robot
//! certificate is never overwritten.
//!
//! ## Robots without a synchronized clock (`--clockless`)
//!
//! TLS checks a certificate's validity window against the wall clock, on both ends of
//! every link. A drone computer without a real-time clock or NTP boots at 1970 (or at its
//! image's build time) and would refuse every teammate, and be refused. Clockless
//! certificates ([`Validity::clockless`]) are valid from the Unix epoch to
//! 9999-12-31 23:59:59 UTC, the date RFC 5280 (§4.1.2.5) sets aside for certificates with
//! no well-defined expiration (as IEEE 802.1AR device identities use it). Authentication
//! is untouched by a wrong clock: a peer still has to hold a key whose certificate the team
//! CA signed, prove it in the mutual handshake, and be in the roster of the access control.
//! What is given up is expiry by date; in its place a team retires certificates by
//! leaving robots out of the roster (`[team.tls] robots`) or by issuing a new team CA
//! (a new `--out`), which every certificate of the old one cannot pass. A clockless team
//! needs a clockless CA: a robot with a wrong clock also checks the CA's own window.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use doorslam_ipc::wire::RobotId;
use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa,
    Issuer, KeyPair, KeyUsagePurpose, SanType,
};

/// The common name of every router's certificate: not a robot id (those have no `.`), so a
/// router can never be mistaken for a robot by the access control, nor the reverse.
pub const ROUTER_COMMON_NAME: &str = "doorslam.router";

/// A new CA is valid for at least this long (robots' certificates for `--days`).
pub const CA_MIN_DAYS: u32 = 3650;

const DAY: Duration = Duration::from_secs(86_400);

/// Failures of certificate generation.
#[derive(Debug, thiserror::Error)]
pub enum CertError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path} already exists: remove it to issue a new one")]
    Exists { path: PathBuf },
    #[error("{present} exists but {missing} does not: the CA needs both (or neither, to create a new one)")]
    HalfCa { present: PathBuf, missing: PathBuf },
    #[error("{path}: {reason}")]
    Ca { path: PathBuf, reason: String },
    #[error("invalid {what} {name:?}: use 1-32 characters of [a-z0-9_-]")]
    Name { what: &'static str, name: String },
    #[error("{0}")]
    Request(String),
    #[error("certificate generation: {0}")]
    Rcgen(#[from] rcgen::Error),
}

/// When a certificate is valid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Validity {
    pub not_before: SystemTime,
    pub not_after: SystemTime,
}

impl Validity {
    /// From an hour ago (clocks of robots and of the issuing machine differ a little) for
    /// `days` days.
    pub fn days_from_now(days: u32) -> Self {
        let now = SystemTime::now();
        Self {
            not_before: now - Duration::from_secs(3600),
            not_after: now + DAY * days,
        }
    }

    /// From the Unix epoch to 9999-12-31 23:59:59 UTC: valid whatever a robot's clock says
    /// (module docs, "Robots without a synchronized clock").
    pub fn clockless() -> Self {
        Self {
            not_before: SystemTime::UNIX_EPOCH,
            not_after: SystemTime::UNIX_EPOCH + Duration::from_secs(CLOCKLESS_NOT_AFTER_UNIX_S),
        }
    }
}

/// 9999-12-31 23:59:59 UTC, RFC 5280's "no well-defined expiration date".
pub const CLOCKLESS_NOT_AFTER_UNIX_S: u64 = 253_402_300_799;

fn offset(t: SystemTime) -> time::OffsetDateTime {
    time::OffsetDateTime::from(t)
}

/// A team's certificate authority: its certificate (PEM) and signing key.
pub struct TeamCa {
    team: String,
    cert_pem: String,
    issuer: Issuer<'static, KeyPair>,
}

impl TeamCa {
    /// A new CA for `team`.
    pub fn create(team: &str, validity: Validity) -> Result<Self, CertError> {
        let team = checked_name("team name", team)?;
        let mut params = CertificateParams::default();
        params.distinguished_name = DistinguishedName::new();
        params
            .distinguished_name
            .push(DnType::CommonName, format!("doorslam team {team} CA"));
        params
            .distinguished_name
            .push(DnType::OrganizationName, team_organization(&team));
        // Signs robots' and routers' certificates only, never another CA.
        params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
        params.key_usages = vec![
            KeyUsagePurpose::KeyCertSign,
            KeyUsagePurpose::CrlSign,
            KeyUsagePurpose::DigitalSignature,
        ];
        params.not_before = offset(validity.not_before);
        params.not_after = offset(validity.not_after);
        let key = KeyPair::generate()?;
        let cert = params.self_signed(&key)?;
        Ok(Self {
            team,
            cert_pem: cert.pem(),
            issuer: Issuer::new(params, key),
        })
    }

    /// The CA of `<dir>/ca.pem` + `<dir>/ca.key`, if both exist.
    pub fn load(dir: &Path) -> Result<Option<Self>, CertError> {
        let (cert_path, key_path) = (dir.join("ca.pem"), dir.join("ca.key"));
        match (cert_path.exists(), key_path.exists()) {
            (false, false) => return Ok(None),
            (true, false) => {
                return Err(CertError::HalfCa {
                    present: cert_path,
                    missing: key_path,
                })
            }
            (false, true) => {
                return Err(CertError::HalfCa {
                    present: key_path,
                    missing: cert_path,
                })
            }
            (true, true) => {}
        }
        let read = |path: &Path| {
            std::fs::read_to_string(path).map_err(|source| CertError::Io {
                path: path.into(),
                source,
            })
        };
        let (cert_pem, key_pem) = (read(&cert_path)?, read(&key_path)?);
        let bad = |path: &Path, reason: String| CertError::Ca {
            path: path.into(),
            reason,
        };
        let key = KeyPair::from_pem(&key_pem)
            .map_err(|e| bad(&key_path, format!("not a PEM private key: {e}")))?;
        let ca = crate::security::parse_certificate_pem(&cert_path, cert_pem.as_bytes())
            .map_err(|e| bad(&cert_path, e.to_string()))?;
        let team = ca
            .organization
            .as_deref()
            .and_then(|o| o.strip_prefix("doorslam team "))
            .map(str::to_string)
            .ok_or_else(|| {
                bad(
                    &cert_path,
                    "not a doorslam team CA (no \"doorslam team <name>\" organization)".into(),
                )
            })?;
        if ca.public_key != key.public_key_raw() {
            return Err(bad(
                &key_path,
                format!("is not the key of {}", cert_path.display()),
            ));
        }
        let issuer = Issuer::from_ca_cert_pem(&cert_pem, key)
            .map_err(|e| bad(&cert_path, format!("not a CA certificate: {e}")))?;
        Ok(Some(Self {
            team,
            cert_pem,
            issuer,
        }))
    }

    pub fn team(&self) -> &str {
        &self.team
    }

    /// Whether the CA's own window is [`Validity::clockless`] (so robots with any clock
    /// accept it).
    pub fn is_clockless(&self) -> bool {
        crate::security::parse_certificate_pem(Path::new("ca.pem"), self.cert_pem.as_bytes())
            .is_ok_and(|c| c.not_before <= 0 && c.not_after >= CLOCKLESS_NOT_AFTER_UNIX_S as i64)
    }

    pub fn cert_pem(&self) -> &str {
        &self.cert_pem
    }

    /// The CA's private key (PEM).
    pub fn key_pem(&self) -> String {
        self.issuer.key().serialize_pem()
    }

    /// A certificate for `common_name` (a robot id, or [`ROUTER_COMMON_NAME`]) signed by this
    /// CA, usable to listen and to connect: `(certificate PEM, private key PEM)`.
    pub fn issue(
        &self,
        common_name: &str,
        validity: Validity,
    ) -> Result<(String, String), CertError> {
        let mut params = CertificateParams::default();
        params.distinguished_name = DistinguishedName::new();
        params
            .distinguished_name
            .push(DnType::CommonName, common_name);
        params
            .distinguished_name
            .push(DnType::OrganizationName, team_organization(&self.team));
        params.subject_alt_names = vec![SanType::DnsName(common_name.try_into()?)];
        params.is_ca = IsCa::ExplicitNoCa;
        params.key_usages = vec![KeyUsagePurpose::DigitalSignature];
        // Every robot both listens and connects.
        params.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        params.use_authority_key_identifier_extension = true;
        params.not_before = offset(validity.not_before);
        params.not_after = offset(validity.not_after);
        let key = KeyPair::generate()?;
        let cert = params.signed_by(&key, &self.issuer)?;
        Ok((cert.pem(), key.serialize_pem()))
    }
}

fn team_organization(team: &str) -> String {
    format!("doorslam team {team}")
}

fn checked_name(what: &'static str, name: &str) -> Result<String, CertError> {
    RobotId::new(name)
        .map(|_| name.to_string())
        .map_err(|_| CertError::Name {
            what,
            name: name.to_string(),
        })
}

/// What `doorslam team certs` asks for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CertsRequest {
    pub team: String,
    pub robots: Vec<String>,
    pub routers: Vec<String>,
    /// Validity of the robots' and routers' certificates (ignored when `clockless`).
    pub days: u32,
    /// Clockless certificates and CA ([`Validity::clockless`]), for robots without a
    /// synchronized clock.
    pub clockless: bool,
}

/// What was written.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Issued {
    pub ca_created: bool,
    pub ca: PathBuf,
    /// `(id, certificate, key)` of each robot, then each router (id `router <name>`).
    pub certificates: Vec<(String, PathBuf, PathBuf)>,
}

/// Writes (or reuses) the team CA in `out` and one certificate per robot and router.
pub fn generate(out: &Path, request: &CertsRequest) -> Result<Issued, CertError> {
    if request.robots.is_empty() && request.routers.is_empty() {
        return Err(CertError::Request(
            "nothing to issue: give --robots and/or --routers".into(),
        ));
    }
    if request.days == 0 && !request.clockless {
        return Err(CertError::Request("--days must be at least 1".into()));
    }
    for r in &request.robots {
        checked_name("robot id", r)?;
    }
    for r in &request.routers {
        checked_name("router name", r)?;
    }
    let team = checked_name("team name", &request.team)?;
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| CertError::Io { path, source }
    };
    std::fs::create_dir_all(out).map_err(io(out))?;
    let ca_path = out.join("ca.pem");
    let (ca, ca_created) = match TeamCa::load(out)? {
        Some(ca) => {
            if ca.team() != team {
                return Err(CertError::Ca {
                    path: ca_path,
                    reason: format!(
                        "is the CA of team {:?}, not {team:?} (use another --out, or --team {})",
                        ca.team(),
                        ca.team()
                    ),
                });
            }
            if request.clockless && !ca.is_clockless() {
                return Err(CertError::Ca {
                    path: ca_path,
                    reason: "is not a clockless CA: a robot whose clock is wrong would refuse it; \
                             issue a clockless team into another --out"
                        .into(),
                });
            }
            (ca, false)
        }
        None => {
            let validity = if request.clockless {
                Validity::clockless()
            } else {
                Validity::days_from_now(request.days.max(CA_MIN_DAYS))
            };
            let ca = TeamCa::create(&team, validity)?;
            write_new(&ca_path, ca.cert_pem(), false)?;
            write_new(&out.join("ca.key"), &ca.key_pem(), true)?;
            (ca, true)
        }
    };
    let validity = if request.clockless {
        Validity::clockless()
    } else {
        Validity::days_from_now(request.days)
    };
    let mut certificates = Vec::new();
    let wanted = request
        .robots
        .iter()
        .map(|r| (out.join("robots").join(r), r.clone(), r.clone()))
        .chain(request.routers.iter().map(|r| {
            (
                out.join("routers").join(r),
                ROUTER_COMMON_NAME.to_string(),
                format!("router {r}"),
            )
        }));
    for (dir, common_name, label) in wanted {
        let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
        for p in [&cert_path, &key_path] {
            if p.exists() {
                return Err(CertError::Exists { path: p.clone() });
            }
        }
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        let (cert, key) = ca.issue(&common_name, validity)?;
        write_new(&key_path, &key, true)?;
        write_new(&cert_path, &cert, false)?;
        certificates.push((label, cert_path, key_path));
    }
    Ok(Issued {
        ca_created,
        ca: ca_path,
        certificates,
    })
}

/// The robot ids that have a certificate under `out/robots/`: the roster every robot's
/// `[team.tls] robots` lists.
pub fn roster(out: &Path) -> Result<Vec<String>, CertError> {
    let dir = out.join("robots");
    let entries = match std::fs::read_dir(&dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(source) => return Err(CertError::Io { path: dir, source }),
    };
    let mut ids = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|source| CertError::Io {
            path: dir.clone(),
            source,
        })?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if entry.path().join("cert.pem").exists() && RobotId::new(&name).is_ok() {
            ids.push(name);
        }
    }
    ids.sort();
    Ok(ids)
}

/// Creates `path` (never overwrites); private keys readable by the owner only.
fn write_new(path: &Path, text: &str, private: bool) -> Result<(), CertError> {
    use std::os::unix::fs::OpenOptionsExt;
    let io = |source| CertError::Io {
        path: path.into(),
        source,
    };
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(if private { 0o600 } else { 0o644 })
        .open(path)
        .map_err(|e| {
            if e.kind() == std::io::ErrorKind::AlreadyExists {
                CertError::Exists { path: path.into() }
            } else {
                io(e)
            }
        })?;
    file.write_all(text.as_bytes()).map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(robots: &[&str]) -> CertsRequest {
        CertsRequest {
            team: "t1".into(),
            robots: robots.iter().map(|s| s.to_string()).collect(),
            routers: vec![],
            days: 30,
            clockless: false,
        }
    }

    #[test]
    fn a_team_ca_signs_robots_and_is_reused_for_later_robots() {
        let dir = tempfile::tempdir().unwrap();
        let issued = generate(dir.path(), &request(&["a", "b"])).unwrap();
        assert!(issued.ca_created);
        assert_eq!(issued.certificates.len(), 2);
        let mode = |p: &Path| {
            use std::os::unix::fs::PermissionsExt;
            std::fs::metadata(p).unwrap().permissions().mode() & 0o777
        };
        assert_eq!(mode(&dir.path().join("ca.key")), 0o600);
        assert_eq!(mode(&issued.certificates[0].2), 0o600);
        let ca_before = std::fs::read(dir.path().join("ca.pem")).unwrap();
        // Later: one more robot, same CA; an existing robot is never reissued silently.
        let later = generate(dir.path(), &request(&["c"])).unwrap();
        assert!(!later.ca_created);
        assert_eq!(std::fs::read(dir.path().join("ca.pem")).unwrap(), ca_before);
        let again = generate(dir.path(), &request(&["a"])).unwrap_err();
        assert!(
            matches!(again, CertError::Exists { .. }),
            "{again}: must refuse to overwrite"
        );
        // Another team's name on this CA is refused, naming the file.
        let mut other = request(&["d"]);
        other.team = "t2".into();
        let err = generate(dir.path(), &other).unwrap_err().to_string();
        assert!(err.contains("ca.pem") && err.contains("t1"), "{err}");
    }

    #[test]
    fn bad_names_and_half_a_ca_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let err = generate(dir.path(), &request(&["A/b"])).unwrap_err();
        assert!(err.to_string().contains("A/b"), "{err}");
        let err = generate(dir.path(), &request(&[])).unwrap_err();
        assert!(err.to_string().contains("--robots"), "{err}");
        std::fs::write(dir.path().join("ca.pem"), "x").unwrap();
        let err = generate(dir.path(), &request(&["a"]))
            .unwrap_err()
            .to_string();
        assert!(err.contains("ca.key"), "{err}");
    }
}
