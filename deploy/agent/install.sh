#!/bin/sh
# Installs `fleet agent` on a robot as fleet-agent.service expects it (run as root):
#   - the system user and group fleet-agent (the unit's User= and Group=);
#   - a virtualenv at /opt/fleet with this package in it (the unit's ExecStart=/opt/fleet/bin/fleet);
#   - /var/spool/robot, where the robot's FileSink recordings go (agent_watch, and the unit's
#     ReadWritePaths=): group fleet-agent, setgid, so add the robot's own user to that group;
#   - /etc/fleet with agent.env (mode 0600: the robot's token goes there) and agent.toml, each left
#     as it is when already there;
#   - the unit, enabled but not started: put the token in /etc/fleet/agent.env first.
# The spool (/var/lib/fleet-agent) is made by systemd itself (StateDirectory=fleet-agent).
#
#   sudo deploy/agent/install.sh [--dry-run]          from a checkout of this repository
#   sudo FLEET_PACKAGE=/tmp/fleet_telemetry-0.1.0-py3-none-any.whl deploy/agent/install.sh
# --dry-run prints the commands instead of running them.
set -eu

AGENT_USER=fleet-agent
PREFIX=/opt/fleet
CONF=/etc/fleet
WATCH=/var/spool/robot
UNITS=/etc/systemd/system
HERE=$(cd "$(dirname "$0")" && pwd)
PACKAGE=${FLEET_PACKAGE:-$(cd "$HERE/../.." && pwd)}
PYTHON=${PYTHON:-python3}

DRY=
if [ "${1:-}" = "--dry-run" ]; then
    DRY=1
fi

run() {
    if [ -n "$DRY" ]; then
        echo "$*"
    else
        "$@"
    fi
}

# whether a user, group or file is there already (a dry run says what a fresh robot needs)
present() {
    [ -z "$DRY" ] && "$@" >/dev/null 2>&1
}

present getent group "$AGENT_USER" || run groupadd --system "$AGENT_USER"
present getent passwd "$AGENT_USER" ||
    run useradd --system --gid "$AGENT_USER" --home-dir /var/lib/fleet-agent --no-create-home \
        --shell /usr/sbin/nologin "$AGENT_USER"

run "$PYTHON" -m venv "$PREFIX"
run "$PREFIX/bin/pip" install --upgrade "$PACKAGE"

run install -d -m 2770 -o "$AGENT_USER" -g "$AGENT_USER" "$WATCH"
run install -d -m 0755 -o root -g root "$CONF"
present test -e "$CONF/agent.env" || run install -m 0600 -o root -g root "$HERE/fleet-agent.env" "$CONF/agent.env"
present test -e "$CONF/agent.toml" || run install -m 0644 -o root -g root "$HERE/agent.toml" "$CONF/agent.toml"

run install -m 0644 "$HERE/fleet-agent.service" "$UNITS/fleet-agent.service"
run systemctl daemon-reload
run systemctl enable fleet-agent

# what is left to do, on stderr (a dry run's stdout is only the commands)
echo "fleet agent installed: set FLEET_TOKEN in $CONF/agent.env, the depot in $CONF/agent.toml, add the" >&2
echo "robot's user to group $AGENT_USER (usermod -aG $AGENT_USER ROBOT_USER), then: systemctl start fleet-agent" >&2
