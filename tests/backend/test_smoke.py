"""The skeleton works on both databases: health, auth by token, visibility of records."""


def test_health(client):
    response = client.get("/api/v1/health")
    assert response.status_code == 200
    assert response.json() == {"status": "ok"}


def test_token_identifies_user(client, world):
    response = client.get("/api/v1/auth/me", headers=world.headers("staff_own"))
    assert response.status_code == 200
    assert response.json()["email"] == "staff-own@example.org"
    assert response.json()["institution"] == "Museum A"


def test_private_record_hidden_from_anonymous(client, world):
    assert client.get(f"/api/v1/tablets/{world.public_a}").status_code == 200
    response = client.get(f"/api/v1/tablets/{world.private_a}")
    assert response.status_code == 404
    assert response.json()["where"] == "tablet_id"
