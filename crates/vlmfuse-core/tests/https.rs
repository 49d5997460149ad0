//! Remote backends over HTTPS: the shared client speaks TLS (rustls, the ring provider) and checks
//! the server's certificate against the system's roots, which `SSL_CERT_FILE` replaces for an
//! internal CA. Against a loopback TLS server with a certificate from a throwaway CA
//! (tests/data/tls): refused while the CA is unknown, answered once it is trusted. One test in
//! its own binary, because it sets an environment variable.

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use std::path::PathBuf;
use std::sync::Arc;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

fn data(f: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/tls")
        .join(f)
}

/// A TLS server answering every request with `{"object": "list", "data": []}`.
async fn tls_server() -> String {
    let _ = rustls::crypto::ring::default_provider().install_default();
    let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(data("cert.pem"))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    let key = PrivateKeyDer::from_pem_file(data("key.pem")).unwrap();
    let cfg = rustls::ServerConfig::builder()
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .unwrap();
    let acceptor = tokio_rustls::TlsAcceptor::from(Arc::new(cfg));
    let l = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    tokio::spawn(async move {
        loop {
            let Ok((s, _)) = l.accept().await else { break };
            let acceptor = acceptor.clone();
            tokio::spawn(async move {
                let Ok(mut tls) = acceptor.accept(s).await else {
                    return;
                };
                let mut buf = Vec::new();
                let mut chunk = [0u8; 1024];
                while !buf.windows(4).any(|w| w == b"\r\n\r\n") {
                    match tls.read(&mut chunk).await {
                        Ok(0) | Err(_) => return,
                        Ok(n) => buf.extend_from_slice(&chunk[..n]),
                    }
                }
                let body = br#"{"object": "list", "data": []}"#;
                let head = format!(
                    "HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ncontent-length: {}\r\nconnection: close\r\n\r\n",
                    body.len()
                );
                let _ = tls.write_all(head.as_bytes()).await;
                let _ = tls.write_all(body).await;
                let _ = tls.shutdown().await;
            });
        }
    });
    format!("https://127.0.0.1:{}/v1/models", addr.port())
}

fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cur = e.source();
    while let Some(c) = cur {
        s.push_str(": ");
        s.push_str(&c.to_string());
        cur = c.source();
    }
    s
}

#[tokio::test(flavor = "multi_thread")]
async fn https_backends_are_reached_and_their_certificates_checked() {
    let url = tls_server().await;

    // An unknown CA: the handshake is made and the certificate refused (never "scheme is not
    // http", as before the client spoke TLS).
    let e = vlmfuse_core::chat::new_http_client()
        .get(&url)
        .send()
        .await
        .unwrap_err();
    let msg = chain(&e);
    assert!(!msg.contains("scheme is not http"), "{msg}");
    assert!(
        msg.to_ascii_lowercase().contains("certificate"),
        "refused for its certificate: {msg}"
    );

    // The CA trusted through SSL_CERT_FILE: answered.
    // SAFETY: this binary's only test sets it before any other thread reads the environment
    // for it (the clients read their roots when built, below).
    unsafe { std::env::set_var("SSL_CERT_FILE", data("ca.pem")) };
    let r = vlmfuse_core::chat::new_http_client()
        .get(&url)
        .send()
        .await
        .unwrap_or_else(|e| panic!("{}", chain(&e)));
    assert_eq!(r.status().as_u16(), 200);
    let v: serde_json::Value = r.json().await.unwrap();
    assert_eq!(v["object"], "list");
}
