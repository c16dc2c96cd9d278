{{- define "lekiwi.name" -}}
{{- default .Chart.Name .Values.nameOverride | trunc 63 | trimSuffix "-" -}}
{{- end -}}

{{- define "lekiwi.fullname" -}}
{{- if .Values.fullnameOverride -}}
{{- .Values.fullnameOverride | trunc 63 | trimSuffix "-" -}}
{{- else -}}
{{- $name := include "lekiwi.name" . -}}
{{- if contains $name .Release.Name -}}
{{- .Release.Name | trunc 63 | trimSuffix "-" -}}
{{- else -}}
{{- printf "%s-%s" .Release.Name $name | trunc 63 | trimSuffix "-" -}}
{{- end -}}
{{- end -}}
{{- end -}}

{{- define "lekiwi.selectorLabels" -}}
app.kubernetes.io/name: {{ include "lekiwi.name" . }}
app.kubernetes.io/instance: {{ .Release.Name }}
{{- end -}}

{{- define "lekiwi.labels" -}}
{{ include "lekiwi.selectorLabels" . }}
app.kubernetes.io/version: {{ .Chart.AppVersion | quote }}
app.kubernetes.io/managed-by: {{ .Release.Service }}
app.kubernetes.io/part-of: lekiwi
helm.sh/chart: {{ printf "%s-%s" .Chart.Name .Chart.Version | replace "+" "_" }}
{{- end -}}

{{- define "lekiwi.serviceAccountName" -}}
{{- if .Values.serviceAccount.create -}}
{{- default (include "lekiwi.fullname" .) .Values.serviceAccount.name -}}
{{- else -}}
{{- default "default" .Values.serviceAccount.name -}}
{{- end -}}
{{- end -}}

{{/* The claim holding events.db and blobs/, or nothing for an emptyDir. */}}
{{- define "lekiwi.claimName" -}}
{{- if .Values.persistence.existingClaim -}}
{{- .Values.persistence.existingClaim -}}
{{- else if .Values.persistence.enabled -}}
{{- printf "%s-data" (include "lekiwi.fullname" .) -}}
{{- end -}}
{{- end -}}

{{/* Whether the event store is the embedded SQLite file (a single writer). */}}
{{- define "lekiwi.sqlite" -}}
{{- if not .Values.store.postgres.existingSecret -}}true{{- end -}}
{{- end -}}

{{/*
Refuses topologies that lose data or split the store, with a message that says what to change.
The schema checks each value; these rules relate several.
*/}}
{{- define "lekiwi.validate" -}}
{{- $v := .Values -}}
{{- if gt (int $v.replicaCount) 1 -}}
{{- if include "lekiwi.sqlite" . -}}
{{- fail (printf "replicaCount=%d needs store.postgres.existingSecret: the SQLite event store has a single writer. Use replicaCount=1, or PostgreSQL plus a ReadWriteMany blob volume (persistence.accessModes=[ReadWriteMany] or a ReadWriteMany persistence.existingClaim)." (int $v.replicaCount)) -}}
{{- end -}}
{{- if and (not $v.persistence.existingClaim) (not $v.persistence.enabled) -}}
{{- fail (printf "replicaCount=%d with persistence.enabled=false gives every replica its own emptyDir blob store: a release pushed to one replica is missing on the others. Enable persistence with accessModes=[ReadWriteMany] or set persistence.existingClaim to a ReadWriteMany claim." (int $v.replicaCount)) -}}
{{- end -}}
{{- if and (not $v.persistence.existingClaim) (not (has "ReadWriteMany" $v.persistence.accessModes)) -}}
{{- fail (printf "replicaCount=%d needs persistence.accessModes to include ReadWriteMany: every replica's gateway serves the release blob store from the same volume (a ReadWriteOnce volume cannot be mounted by pods on several nodes)." (int $v.replicaCount)) -}}
{{- end -}}
{{- end -}}
{{- if and $v.podDisruptionBudget.enabled (kindIs "invalid" $v.podDisruptionBudget.minAvailable) (kindIs "invalid" $v.podDisruptionBudget.maxUnavailable) -}}
{{- fail "podDisruptionBudget: set minAvailable or maxUnavailable (or enabled=false)" -}}
{{- end -}}
{{- end -}}

{{/* The TLS Secret the gateway serves with: the given one, the generated one, or nothing for
plain text (gateway.tls.enabled=false). */}}
{{- define "lekiwi.tlsSecret" -}}
{{- if .Values.gateway.tls.secretName -}}
{{- .Values.gateway.tls.secretName -}}
{{- else if include "lekiwi.tlsGenerated" . -}}
{{- printf "%s-gateway-tls" (include "lekiwi.fullname" .) -}}
{{- end -}}
{{- end -}}

{{/* Whether the chart makes the gateway's CA and certificate itself (TLS on, no Secret given,
and a gateway runs: not for role=controller). */}}
{{- define "lekiwi.tlsGenerated" -}}
{{- if and .Values.gateway.tls.enabled (not .Values.gateway.tls.secretName) (ne .Values.operator.role "controller") -}}true{{- end -}}
{{- end -}}
